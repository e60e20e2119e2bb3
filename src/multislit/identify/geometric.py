"""Identification by the dots' geometry: the chain of stages from an image to its labels.

1. the stripes and the dot image (:func:`~multislit.stripes.extract_slits`), and the dots
   found in it (:func:`~multislit.identify.evidence.frame_dots`);
2. the linked stripe points in windows of consecutive rows
   (:func:`~multislit.identify.pieces.windows`), and for every window, slit and side of the
   stripe, how well the slit explains the dots beside it
   (:func:`~multislit.identify.evidence.dot_evidence`);
3. the gaps between windows side by side in the rows (:func:`~multislit.identify.pieces.gaps`)
   and what the dots between them say (:func:`~multislit.identify.evidence.gap_evidence`); the
   windows that continue one another: the next window of a segment, and a segment that
   continues another below it (:func:`~multislit.identify.pieces.continuations`);
4. one labelling of all the windows (:func:`~multislit.identify.graph.label_pieces`): a
   window below the required confidence is left out. Where a segment's slit changes (the
   linking joined two slits' stripes where they meet), its windows take different labels:
   each change costs the chain's bonus, so the dots decide where;
5. the pieces: each segment cut where its windows' labels change.

Each stage returns a new value; the result says per piece where its label came from
(:class:`~multislit.identify.result.PieceLabels`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from multislit.identify.evidence import (
    dot_evidence,
    dot_matches,
    frame_dots,
    gap_evidence,
    window_stripes,
)
from multislit.identify.graph import confidence_margin, label_pieces
from multislit.identify.options import IdentifyOptions
from multislit.identify.pieces import (
    Gaps,
    Windows,
    continuations,
    gaps_across,
    split_at_kinks,
    windows,
)
from multislit.identify.reference import ReferenceSet
from multislit.identify.result import SOURCES, Identification, PieceLabels
from multislit.identify.rig import RigGeometry
from multislit.identify.segments import split_at_brightness_steps
from multislit.identify.shadows import shadow_factors
from multislit.stripes import SlitExtraction

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Stripe points per window (rows): the dots' evidence is scored per window, the surface's
#: slope across the stripe free in each.
_WINDOW_ROWS = 24
#: Log-likelihood a window gains when it carries the slit of the window before it in its
#: segment, and loses when it carries another (where the segment crosses an object's edge).
_CHAIN = 4.0
_CHAIN_CHANGE = 1.5
#: Rows left out on either side of a change of slit between two windows of a segment.
_JUNCTION_ROWS = 8
#: A segment is cut where its brightness steps by this ratio (the medians of 6 points before and
#: after): a cut links its pieces as a junction (:data:`_JUNCTION`), so a piece beyond it must
#: stand on its own dots ...
_STEP_CUT = 1.45
#: ... and where lines fitted to this many points before and after a point put the
#: stripe more than this many px apart (a step where two slits' stripes meet).
_KINK_ROWS = 6
_KINK_PX = 0.5
#: Pieces farther apart in a row than this many slit spacings are not neighbours there ...
_GAP_SPACINGS = 3.0
#: ... and pieces side by side in fewer rows than this are not neighbours at all.
_GAP_ROWS = 3
#: Log-likelihood a gap gains when its pieces are neighbouring slits of one surface ...
_COUPLING = 6.0
#: ... less where the gap's width is off the widths of the gaps beside it by more than this
#: factor (a Gaussian in the log of the ratio) ...
_SPACING_TOLERANCE = 1.3
#: ... or where its two stripes' brightness differs by more than this factor (the same): stripes
#: of one surface look alike, one beside an object's edge often does not ...
_BRIGHTNESS_TOLERANCE = 2.2
#: ... and none where that surface meets a line of sight at less than acos(this).
_GRAZE = 0.97
#: Log-likelihood a gap loses when both its pieces carry one slit ...
_REPEAT_PENALTY = 30.0
#: ... and when they carry slits that are not neighbours of one surface (a step in depth).
_SPLIT = 1.5
#: A window is labelled only when the dots' evidence of the group of windows its label ties it
#: to (neighbouring slits of one surface, continuations of one slit) reaches this (nats).
_MIN_SUPPORT = 8.0
#: Why a piece with slits in the measuring volume is left out: its slit rests on a
#: continuation across a cut alone (:func:`_continuations`), the dots of the group of pieces
#: its label ties it to say less than :data:`_MIN_SUPPORT`, or its confidence is below the
#: required one.
_LEFT_OUT = ("rests_on_a_cut", "too_little_evidence", "low_confidence")
#: The windows' slits of the lowest evidence (from the rank on) measure the frame's evidence
#: under wrong slits, which is taken out of every window's so that chance does not add up.
_NULL_RANK = 4
#: Across a cut of a linked segment (a brightness step or a kink), the window after it gains
#: this for the slit of the window before it.
_JUNCTION = 5.0
#: The dots between two windows are scored for the pairs (k, k + 1) of slits within this (nats)
#: of each window's best.
_PAIR_NATS = 8.0
#: A piece that continues another below it (within these rows and px) gains this for one slit.
_CONTINUATION = 1.0
_CONTINUATION_ROWS = 12
_CONTINUATION_PX = 4.0
#: ... and as bright, within this ratio.
_STEP_RATIO = 1.6


def _empty(ex: SlitExtraction, message: str) -> Identification:
    k = len(ex.u)
    return Identification(
        ex.u,
        ex.v,
        np.full(k, -1, np.int64),
        np.zeros(k),
        np.full(k, -1, np.int64),
        ex.peak,
        ex.width,
        0,
        0,
        {},
        message,
        ex,
        None,
        "geometry",
    )


def identify_geometry(
    ex: SlitExtraction,
    reference: ReferenceSet,
    rig: RigGeometry,
    options: IdentifyOptions,
    match_dots: bool = True,
) -> Identification:
    """Label the stripe points of an extraction by the dots' geometry (see the module).

    Parameters
    ----------
    ex : the image's extraction
    reference : the rig's prepared reference (its slit spacing)
    rig : the calibrated rig (:func:`~multislit.identify.rig.rig_geometry`)
    options : the identification's options (``min_confidence``)
    match_dots : also pair the observed dots beside the labelled windows with the projector's
        rays (:func:`~multislit.identify.evidence.dot_matches`); False: ``dots`` is None

    Returns
    -------
    Identification with ``pieces`` and ``method="geometry"``
    """
    k = len(ex.u)
    if k == 0 or not np.any(ex.segment >= 0):
        return _empty(ex, "no slits found in the image")
    frame = frame_dots(ex, reference.spacing_px)
    uv = np.stack([ex.u, ex.v], axis=1)
    _, rays = rig.camera.rays(uv)
    # each point's position along its stripe and across it: its row and column, or its column
    # and row where it was found along the columns
    along = np.where(ex.by_column, ex.u, ex.v)
    across = np.where(ex.by_column, ex.v, ex.u)
    # where a stripe runs into another surface's stripe the linking may join them; the
    # brightness steps there (another albedo or depth)
    segment = split_at_brightness_steps(
        ex.segment.astype(np.int64), along, ex.peak, ratio=_STEP_CUT
    )
    segment = split_at_kinks(segment, across, along, _KINK_ROWS, _KINK_PX)
    win = windows(segment, along, _WINDOW_ROWS)
    w_dir, w_peak = window_stripes(ex, win.order, win.start)
    ev = dot_evidence(rig, rays, win.order, win.start, frame, w_dir, w_peak)
    scores = _calibrated(ev.llr.sum(axis=2).astype(np.float64))
    nw = win.num_windows
    window = Windows(win.order, win.start, win.segment, np.arange(nw)).piece_of_points(k)
    gp = gaps_across(
        ex.u, ex.v, window, ex.by_column, ex.angle, _GAP_SPACINGS * reference.spacing_px, _GAP_ROWS
    )
    # the pairs (k, k + 1) worth the dots between: both near their windows' best
    best = np.where(np.isfinite(scores), scores, -np.inf)
    near_best = ev.kept & (best >= best.max(axis=1, keepdims=True) - _PAIR_NATS)
    pairs = np.zeros((gp.num_gaps, rig.num_slits), bool)
    pairs[:, :-1] = near_best[gp.a, :-1] & near_best[gp.b, 1:]
    ge = gap_evidence(
        rig,
        rays,
        gp.a_order,
        gp.a_start,
        gp.b_order,
        gp.b_start,
        frame,
        0.5 * (w_dir[gp.a] + w_dir[gp.b]),
        np.sqrt(w_peak[gp.a] * w_peak[gp.b]),
        gp.a,
        gp.b,
        ev,
        pairs,
    )
    ca, cb, bonus, change, vouch = _continuations(ex, ex.segment.astype(np.int64), segment, win)
    # the dots between them count where scored; elsewhere the pieces' own evidence stands
    between = np.where(np.isfinite(ge.fixed), ge.bonus, 0.0).astype(np.float64)
    # a gap much wider or narrower than those beside it, or between stripes of much unlike
    # brightness, is a step between two surfaces more often than a stretch of one: its coupling
    # weighs less
    regular = _regularity(gp.spacing_ratio, _brightness_ratio(ex.peak, gp))

    def labelling(factors=None, ties=vouch):
        return label_pieces(
            scores,
            gp.a,
            gp.b,
            between,
            np.isfinite(ge.graze) & (ge.graze < _GRAZE),
            gp.rows,
            ca,
            cb,
            bonus,
            change,
            coupling=_COUPLING * regular,
            gap_pair=win.segment[gp.a] * (int(win.segment.max()) + 1) + win.segment[gp.b],
            repeat_penalty=_REPEAT_PENALTY,
            split_penalty=_SPLIT,
            cont_ties=ties,
            factors=factors,
        )

    # a first labelling, for where the confident stripes are (their shadows' gaps)
    lab = labelling(ties=None)
    sure = (lab.slit >= 0) & (lab.confidence >= options.confidence) & (lab.support >= _MIN_SUPPORT)
    lab = labelling(shadow_factors(ev.span, lab.slit, sure))
    accepted = (
        (lab.slit >= 0) & (lab.confidence >= options.confidence) & (lab.support >= _MIN_SUPPORT)
    )
    label = np.where(accepted, lab.slit, -1)
    # the pieces: runs of windows of one linked segment, along it, with one label (across a
    # cut whose two sides carry one slit too)
    head = win.order[win.start[:-1]]
    linked = ex.segment[head]
    o = np.lexsort((along[head], linked))
    new = np.r_[True, (linked[o][1:] != linked[o][:-1]) | (label[o][1:] != label[o][:-1])]
    piece_of_window = np.empty(nw, np.int64)
    piece_of_window[o] = np.cumsum(new) - 1
    piece = np.full(k, -1, np.int64)
    piece[window >= 0] = piece_of_window[window[window >= 0]]
    # why each window left out is: its slit rests on a cut alone, its group's dots say too
    # little, or the labelling is not confident enough
    why = np.where(
        lab.rests_on_cut,
        _LEFT_OUT.index("rests_on_a_cut"),
        np.where(
            lab.support < _MIN_SUPPORT,
            _LEFT_OUT.index("too_little_evidence"),
            _LEFT_OUT.index("low_confidence"),
        ),
    )
    pieces, dropped = _piece_labels(
        scores, piece_of_window, label, lab.confidence, options.confidence, why
    )
    dots = None
    if match_dots:
        lw = np.flatnonzero(label >= 0)
        dots = dot_matches(
            rig,
            rays,
            win.order,
            win.start,
            frame,
            lw,
            label[lw],
            ev.slope[lw, label[lw]].astype(np.float64),
            lab.confidence[lw],
            w_dir,
        )
    slit = np.full(k, -1, np.int64)
    conf = np.zeros(k)
    has = window >= 0
    slit[has] = label[window[has]]
    conf[has] = np.where(slit[has] >= 0, lab.confidence[window[has]], 0.0)
    # where a linked stripe's slit changes between two windows (within a piece or across a cut),
    # the change lies somewhere in them: the rows next to their boundary are left out
    slit[_near_changes(along, win, label, linked)] = -1
    conf[slit < 0] = 0.0
    return Identification(
        ex.u,
        ex.v,
        slit,
        conf,
        piece,
        ex.peak,
        ex.width,
        len(pieces.slit),
        int(np.count_nonzero(pieces.slit >= 0)),
        dropped,
        "",
        ex,
        pieces,
        "geometry",
        dots,
    )


def _brightness_ratio(peak: F64, gp: Gaps) -> F64:
    """(G,) each gap's left stripe's brightness over its right one's: the ratio of the
    geometric means of their peaks (``peak`` (K,), per point) over the rows they share."""
    n = np.diff(gp.a_start)
    gap = np.repeat(np.arange(gp.num_gaps), n)
    d = np.log(np.maximum(peak[gp.a_order], 1e-9) / np.maximum(peak[gp.b_order], 1e-9))
    return np.exp(np.bincount(gap, d, minlength=gp.num_gaps) / np.maximum(n, 1))


def _regularity(spacing_ratio: F64, brightness_ratio: F64) -> F64:
    """(G,) 0..1, the weight of each gap's coupling: a Gaussian in the log of its width's
    ratio to the widths beside it (scale log :data:`_SPACING_TOLERANCE`; 1 where none is
    beside it) times one in the log of its stripes' brightness ratio (scale log
    :data:`_BRIGHTNESS_TOLERANCE`)."""
    out = np.ones(len(spacing_ratio))
    for ratio, tol in (
        (spacing_ratio, _SPACING_TOLERANCE),
        (brightness_ratio, _BRIGHTNESS_TOLERANCE),
    ):
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.log(ratio) / math.log(tol)
        out *= np.where(np.isfinite(x), np.exp(-0.5 * x**2), 1.0)
    return out


def _calibrated(scores: F64) -> F64:
    """The windows' log-likelihood ratios (W, N) less the frame's bias under wrong slits: the
    log of the mean of exp(ratio) over each window's slits from the :data:`_NULL_RANK`-th best
    on (a calibrated ratio averages 1 there; chance finds of dots make it more)."""
    x = np.where(np.isfinite(scores), scores, -np.inf)
    if x.shape[1] <= _NULL_RANK:
        return scores
    rest = -np.sort(-x, axis=1)[:, _NULL_RANK:]
    rest = rest[np.isfinite(rest)]
    if rest.size == 0:
        return scores
    top = rest.max()
    bias = top + math.log(np.mean(np.exp(rest - top)))
    return scores - max(bias, 0.0)


def _near_changes(along: F64, win: Windows, label: I64, linked: I64) -> NDArray[np.bool_]:
    """(K,) bool: the points within :data:`_JUNCTION_ROWS` rows (columns, for a segment found
    along the columns; ``along`` (K,) px, the position along the stripe) of a boundary between
    two windows next to each other along one linked stripe whose labels differ (both
    labelled). ``linked`` (W,): each window's linked stripe (the extraction's segment), so a
    boundary at a cut (a brightness step, a kink: where a change is likeliest) counts as one
    within a piece."""
    out = np.zeros(len(along), bool)
    head = win.order[win.start[:-1]]
    o = np.lexsort((along[head], linked))
    a, b = o[:-1], o[1:]
    changes = np.flatnonzero((linked[a] == linked[b]) & (linked[a] >= 0) & (label[a] != label[b]))
    changes = changes[(label[a[changes]] >= 0) & (label[b[changes]] >= 0)]
    for i in changes:  # the boundary: between window a's last point and b's first
        pa = win.order[win.start[a[i]] : win.start[a[i] + 1]]
        pb = win.order[win.start[b[i]] : win.start[b[i] + 1]]
        mid = 0.5 * (along[pa].max() + along[pb].min())
        both = np.r_[pa, pb]
        out[both[np.abs(along[both] - mid) <= _JUNCTION_ROWS]] = True
    return out


def _continuations(
    ex: SlitExtraction, linked: I64, segment: I64, win: Windows
) -> tuple[I64, I64, F64, F64, NDArray[np.bool_]]:
    """The windows that continue one another, the bonus of one slit and the cost of two for
    each, and whether they vouch for each other: the next window of a segment
    (:data:`_CHAIN`, :data:`_CHAIN_CHANGE`; they vouch); across a cut of a linked segment
    (``linked``, the extraction's segments; ``segment``, them cut at brightness steps and
    kinks), the first window after the cut (:data:`_JUNCTION`: the cut may be where two slits'
    stripes meet, or a bend or a shading step of one; they do not vouch: a slit must not rest
    on continuity across a cut alone); and the first window of a segment that continues another
    below it, as bright (:data:`_CONTINUATION`; they vouch)."""
    nw = win.num_windows
    same = np.flatnonzero(win.segment[1:] == win.segment[:-1])
    nseg = int(win.segment.max()) + 1 if nw else 0
    first = np.full(nseg, -1, np.int64)
    last = np.full(nseg, -1, np.int64)
    first[win.segment[::-1]] = np.arange(nw)[::-1]
    last[win.segment] = np.arange(nw)
    # the pieces of one linked segment, in their order along it
    along = np.where(ex.by_column, ex.u, ex.v)
    has = first >= 0
    head = win.order[win.start[first[has]]]
    pieces = np.flatnonzero(has)
    o = np.lexsort((along[head], linked[head]))
    pieces, head = pieces[o], head[o]
    nxt = np.flatnonzero(linked[head[1:]] == linked[head[:-1]])
    ja, jb = last[pieces[nxt]], first[pieces[nxt + 1]]
    sa, sb = continuations(ex.u, ex.v, segment, _CONTINUATION_ROWS, _CONTINUATION_PX)
    if len(sa):
        # the (geometric) mean brightness of the windows that meet: a step is another surface
        logp = np.log(np.maximum(ex.peak[win.order], 1e-6))
        wpeak = np.exp(np.add.reduceat(logp, win.start[:-1]) / np.diff(win.start))
        ratio = wpeak[last[sa]] / np.maximum(wpeak[first[sb]], 1e-6)
        keep = (ratio < _STEP_RATIO) & (ratio > 1.0 / _STEP_RATIO)
        # a cut's pieces are linked as a junction already
        keep &= linked[win.order[win.start[last[sa]]]] != linked[win.order[win.start[first[sb]]]]
        sa, sb = sa[keep], sb[keep]
    a = np.r_[same, ja, last[sa]].astype(np.int64)
    b = np.r_[same + 1, jb, first[sb]].astype(np.int64)
    bonus = np.r_[
        np.full(len(same), _CHAIN), np.full(len(ja), _JUNCTION), np.full(len(sa), _CONTINUATION)
    ]
    change = np.r_[np.full(len(same), _CHAIN_CHANGE), np.zeros(len(ja)), np.zeros(len(sa))]
    vouch = np.r_[np.ones(len(same), bool), np.zeros(len(ja), bool), np.ones(len(sa), bool)]
    return a, b, bonus, change, vouch


def _piece_labels(
    scores: F64,
    piece_of_window: I64,
    label: I64,
    confidence: F64,
    min_confidence: float,
    why: I64,
) -> tuple[PieceLabels, dict[str, int]]:
    """Per piece (a run of windows with one label): its label and confidence (the least of
    its windows'), its own dots' preference and where its label came from; and the counts of
    the pieces left out by reason: ``out_of_volume`` (every slit puts it outside the measuring
    volume), else the reason (:data:`_LEFT_OUT`, ``why`` (W,) per window) of most of its
    windows."""
    s = int(piece_of_window.max()) + 1
    n = scores.shape[1]
    own_scores = np.zeros((s, n))
    np.add.at(own_scores, piece_of_window, np.where(np.isfinite(scores), scores, 0.0))
    ruled = np.zeros((s, n), bool)
    np.logical_or.at(ruled, piece_of_window, ~np.isfinite(scores))
    u = np.where(ruled, -np.inf, own_scores)
    valid = np.isfinite(u).any(axis=1)
    order = np.argsort(-u, axis=1)
    own = np.where(valid, order[:, 0], -1)
    best = u[np.arange(s), order[:, 0]]
    second = u[np.arange(s), order[:, 1]] if n > 1 else np.full(s, -np.inf)
    own_margin = np.where(valid, np.minimum(best - np.maximum(second, 0.0), best), 0.0)
    slit = np.full(s, -1, np.int64)
    slit[piece_of_window] = label
    conf = np.ones(s)
    np.minimum.at(conf, piece_of_window, confidence)
    accepted = slit >= 0
    need = confidence_margin(min_confidence) if min_confidence > 0 else -math.inf
    by_dots = accepted & (own == slit) & (own_margin >= need)
    source = np.zeros(s, np.int8)
    source[accepted] = SOURCES.index("its neighbours")
    source[by_dots] = SOURCES.index("its dots")
    votes = np.zeros((s, len(_LEFT_OUT)), np.int64)
    np.add.at(votes, (piece_of_window, why), 1)
    reason = np.argmax(votes, axis=1)
    left = valid & ~accepted
    dropped = {"out_of_volume": int(np.count_nonzero(~valid))}
    for i, name in enumerate(_LEFT_OUT):
        dropped[name] = int(np.count_nonzero(left & (reason == i)))
    return PieceLabels(slit, conf, own.astype(np.int64), own_margin, source), dropped

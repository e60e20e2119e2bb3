"""One labelling of all the pieces of a frame: their own dots and what their neighbours say.

Every piece gets the slit of the labelling that maximises

- each piece's own evidence: the log-likelihood ratio of its dots per slit
  (:mod:`~multislit.identify.evidence`; a slit that puts the piece outside the measuring
  volume is ruled out);
- per gap (two pieces side by side in the rows, :func:`~multislit.identify.pieces.gaps`): when
  the right piece is the next slit of the left one and the surface through both stripes does
  not graze the camera's or the dot source's line of sight, a coupling (``coupling``, scaled
  by the rows they share) plus what the dots between them say for one surface against each
  piece alone (:attr:`~multislit.identify.evidence.GapEvidence.bonus`); when both carry one
  slit, a penalty (a slit lights a row once);
- per continuation (a piece that continues another: the next window of a segment, or a
  segment that continues another below it): a bonus for one slit. Some continuations do not
  vouch (across a place where two slits' stripes may meet): a piece whose slit rests on
  them alone is left out.

The labelling is found by loopy belief propagation (max-product, undamped, for at most
:data:`_SWEEPS` sweeps: on loops of pieces its messages may keep cycling instead of settling),
which gives every piece its belief per label; the confidence of a piece's label is its
belief's share (softmax) against every other slit; the support of a label is the own evidence
summed over the group of pieces the labelling ties together. A piece whose best slit has less
than the required confidence or support is left out, never guessed.

Units: log-likelihood (nats).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from multislit.identify.launch import launch

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Rows two pieces must share for their coupling to count in full.
_COUPLING_ROWS = 40.0
#: Belief propagation: at most this many sweeps ...
_SWEEPS = 10
#: ... stopping once no message moves by more than this (nats).
_SETTLED = 0.05
#: A message is sent again only when its source's belief has moved by more than this (nats)
#: since it was last sent.
_QUIET = 1e-3


@dataclass(frozen=True, eq=False)
class Labelling:
    """The frame's labelling.

    Attributes
    ----------
    slit : (S,) int64, each piece's best slit (-1: every slit ruled out)
    confidence : (S,) float64, 0..1, the best slit's share of the belief against every other
    belief : (S, N) float64, max-product beliefs
    support : (S,) float64, nats, the dots' evidence for the labelling of the group of pieces
        it ties the piece to (by the gaps of neighbouring slits and the continuations of one
        slit): the sum of their own log-likelihood ratios for their labels
    rests_on_cut : (S,) bool, the piece's best slit is another in the labelling without the
        continuations that do not vouch: its slit rests on them alone (its confidence is 0)
    """

    slit: I64
    confidence: F64
    belief: F64
    support: F64
    rests_on_cut: NDArray[np.bool_]


@njit(cache=True)
def _top3(h):
    """Indices of the three largest values of ``h`` (fewer when shorter: -1)."""
    i1 = i2 = i3 = -1
    for k in range(len(h)):
        x = h[k]
        if i1 < 0 or x > h[i1]:
            i3, i2, i1 = i2, i1, k
        elif i2 < 0 or x > h[i2]:
            i3, i2 = i2, k
        elif i3 < 0 or x > h[i3]:
            i3 = k
    return i1, i2, i3


@njit(cache=True, inline="always")
def _max_except(h, t1, t2, t3, x, y):
    """The largest value of ``h`` at an index other than ``x`` and ``y`` (its three largest
    at ``t1``, ``t2``, ``t3``)."""
    for t in (t1, t2, t3):
        if t >= 0 and t != x and t != y:
            return h[t]
    return -np.inf


@njit(cache=True)
def _gap_message(h, theta, penalty, split, forward, out):
    """The message across a gap: from the left piece (``forward``) or from the right one.
    ``theta`` (N,): the coupling when the right piece is slit k + 1 of the left one's k (NaN:
    no coupling: a step in depth); ``penalty``: the cost of both carrying one slit; ``split``:
    the cost of two slits that are not neighbours of one surface."""
    n = len(h)
    t1, t2, t3 = _top3(h)
    for k in range(n):
        if forward:  # to the right piece's k from the left piece's k - 1
            c = k - 1
            best = _max_except(h, t1, t2, t3, k, c if c >= 0 else -2) - split
            if c >= 0:
                best = max(best, h[c] + (theta[c] if np.isfinite(theta[c]) else -split))
        else:  # to the left piece's k from the right piece's k + 1
            c = k + 1
            best = _max_except(h, t1, t2, t3, k, c if c < n else -2) - split
            if c < n:
                best = max(best, h[c] + (theta[k] if np.isfinite(theta[k]) else -split))
        out[k] = max(best, h[k] - penalty)


@njit(cache=True)
def _continuation_message(h, bonus, change, out):
    """The message along a continuation: one slit gains ``bonus``, two slits lose ``change``."""
    t1, t2, t3 = _top3(h)
    for k in range(len(h)):
        out[k] = max(_max_except(h, t1, t2, t3, k, -2) - change, h[k] + bonus)


@njit(cache=True)
def _propagate(unary, ga, gb, theta, penalty, split, ca, cb, bonus, change, f_slit, f_cost,
               f_start, f_cand, sweeps):  # fmt: skip
    """Loopy max-product belief propagation; the beliefs (S, L) and the messages along each
    edge (gaps, then continuations) to its second piece and to its first (E, L) each.

    Beside the edges, "one of them" factors: factor f wants one of its candidate pieces
    ``f_cand[f_start[f]:f_start[f+1]]`` to carry slit ``f_slit[f]`` and costs ``f_cost[f]``
    when none does; its message favours that slit for a candidate by the least regret of the
    other candidates to carry it (at most the cost).

    The messages are sent one after the other, each piece's belief kept up to date as they
    arrive, the edges in their order and in reverse by turns (a chain's evidence travels its
    length in one sweep). Each piece's belief has a version, raised whenever a message moves
    it by more than :data:`_QUIET`; a message whose source's version is the one it was last
    computed from is not computed again (it would come out the same), so after the first
    sweeps only the messages near a change are."""
    nl = unary.shape[1]
    ng = len(ga)
    ne = ng + len(ca)
    # messages: edge e forward (to its second piece) and backward (to its first)
    fwd = np.zeros((ne, nl))
    bwd = np.zeros((ne, nl))
    orm = np.zeros(len(f_cand))  # factor -> candidate: how much its slit is favoured
    belief = unary.copy()
    tmp = np.empty(nl)
    h = np.empty(nl)
    version = np.zeros(len(unary), np.int64)
    sent = np.full((ne, 2), -1, np.int64)  # the source's version each message was sent from
    for sweep in range(sweeps):
        moved = 0.0
        for q in range(ne):
            e = q if sweep % 2 == 0 else ne - 1 - q
            a = ga[e] if e < ng else ca[e - ng]
            b = gb[e] if e < ng else cb[e - ng]
            for forward in (True, False):
                # from one end of the edge, without what the other end told it
                src, dst = (a, b) if forward else (b, a)
                side = 0 if forward else 1
                if sent[e, side] == version[src]:
                    continue
                sent[e, side] = version[src]
                msg = fwd[e] if forward else bwd[e]
                back = bwd[e] if forward else fwd[e]
                for k in range(nl):
                    h[k] = belief[src, k] - back[k]
                if e < ng:
                    _gap_message(h, theta[e], penalty[e], split[e], forward, tmp)
                else:
                    _continuation_message(h, bonus[e - ng], change[e - ng], tmp)
                m = tmp.max()
                step = 0.0
                for k in range(nl):
                    x = tmp[k] - m
                    step = max(step, abs(x - msg[k]))
                    belief[dst, k] += x - msg[k]
                    msg[k] = x
                moved = max(moved, step)
                if step > _QUIET:
                    version[dst] += 1
        for f in range(len(f_slit)):
            k = f_slit[f]
            r1 = r2 = np.inf
            i1 = -1
            for q in range(f_start[f], f_start[f + 1]):
                i = f_cand[q]
                # the candidate's regret to carry k, without this factor's message
                top = belief[i, k]
                for l in range(nl):
                    if l != k:
                        top = max(top, belief[i, l] + orm[q])
                r = top - belief[i, k]
                if r < r1:
                    r2, r1, i1 = r1, r, q
                elif r < r2:
                    r2 = r
            for q in range(f_start[f], f_start[f + 1]):
                x = min(f_cost[f], r2 if q == i1 else r1)
                d = x - orm[q]
                moved = max(moved, abs(d))
                i = f_cand[q]
                if abs(d) > _QUIET:
                    version[i] += 1
                # the message favours k by orm: the other labels lose it
                for l in range(nl):
                    if l != k:
                        belief[i, l] -= d
                orm[q] = x
        if moved < _SETTLED:
            break
    return belief, fwd, bwd


@njit(cache=True, parallel=True)
def _propagate_pair(unary, ga, gb, theta, penalty, split, ca, cb, bonus, change, ca2, cb2,
                    bonus2, change2, second, f_slit, f_cost, f_start, f_cand):  # fmt: skip
    """The beliefs (S, L) of :func:`_propagate` with the continuations ``ca``, ``cb``,
    ``bonus``, ``change`` and, when ``second``, beside them (on another of Numba's threads)
    with the continuations ``ca2`` .. ``change2`` instead (else the second is empty)."""
    out = np.empty((2 if second else 1, unary.shape[0], unary.shape[1]))
    for i in prange(out.shape[0]):
        if i == 0:
            b, _, _ = _propagate(unary, ga, gb, theta, penalty, split, ca, cb, bonus, change,
                                 f_slit, f_cost, f_start, f_cand, _SWEEPS)  # fmt: skip
        else:
            b, _, _ = _propagate(unary, ga, gb, theta, penalty, split, ca2, cb2, bonus2, change2,
                                 f_slit, f_cost, f_start, f_cand, _SWEEPS)  # fmt: skip
        out[i] = b
    if second:
        return out[0], out[1]
    return out[0], np.empty((0, unary.shape[1]))


def label_pieces(
    unary: F64,
    gap_a: I64,
    gap_b: I64,
    gap_bonus: F64,
    gap_continuous: NDArray[np.bool_],
    gap_rows: I64,
    cont_a: I64,
    cont_b: I64,
    cont_bonus: F64,
    cont_change: F64,
    *,
    coupling: float | F64,
    repeat_penalty: float,
    split_penalty: float,
    gap_pair: I64 | None = None,
    cont_ties: NDArray[np.bool_] | None = None,
    factors: tuple | None = None,
) -> Labelling:
    """The labelling of the frame's pieces (see the module's docstring).

    Parameters
    ----------
    unary : (S, N) float64, each piece's log-likelihood ratio per slit (NaN: ruled out)
    gap_a, gap_b : (G,) int64, the left and right piece of each gap
    gap_bonus : (G, N) float64, what the dots between them say for (k, k + 1) on one surface
        against each piece alone (NaN: not a hypothesis)
    gap_continuous : (G, N) bool, the surface through both stripes under (k, k + 1) does not
        graze a line of sight
    gap_rows : (G,) int64, the rows each gap's pieces share
    cont_a, cont_b : (C,) int64, continuations: piece b continues piece a
    cont_bonus : (C,) float64, log-likelihood a continuation gains when both carry one slit
    cont_change : (C,) float64, log-likelihood it loses when they carry two slits
    coupling : log-likelihood gained by a gap whose pieces are neighbouring slits of one
        surface (for the full :data:`_COUPLING_ROWS` shared rows; less for fewer); a number,
        or (G,) one per gap
    gap_pair : (G,) int64, the pair of stripes (segments) each gap lies between, or None. That
        two stripes side by side are neighbouring slits is one fact however long they run
        side by side: the gaps of one pair share its coupling by their rows, in full for
        :data:`_COUPLING_ROWS` shared rows in all (the dots between them, ``gap_bonus``, count
        gap by gap). None: each gap couples on its own.
    cont_ties : (C,) bool, the continuations whose pieces, when they carry one slit, vouch
        for each other: their own evidence adds up in ``support``, and a piece's slit may rest
        on them (default all). The frame is labelled a second time without the continuations
        that do not vouch; a piece whose best slit differs there rests on them alone, and its
        confidence is 0.
    factors : (slit (F,), cost (F,), start (F+1,), candidates (M,)) or None: "one of them"
        factors (:func:`_propagate`): factor f costs ``cost[f]`` unless one of the pieces
        ``candidates[start[f]:start[f+1]]`` carries ``slit[f]``
    repeat_penalty : log-likelihood lost by a gap whose pieces carry one slit
    split_penalty : log-likelihood lost by a gap whose pieces carry two slits that are not
        neighbours of one surface (a step in depth)

    Returns
    -------
    Labelling; ``support`` says which pieces the dots support
    """
    s, n = unary.shape
    u = np.where(np.isfinite(unary), unary, -1e9)
    rows = np.asarray(gap_rows, np.float64)
    w = np.minimum(1.0, rows / _COUPLING_ROWS)
    cont = gap_continuous & np.isfinite(gap_bonus)
    share = w
    if gap_pair is not None and rows.size:
        _, pair = np.unique(np.asarray(gap_pair), return_inverse=True)
        share = rows / np.maximum(np.bincount(pair, rows)[pair], _COUPLING_ROWS)
    cw = np.broadcast_to(np.asarray(coupling, np.float64), w.shape) * share
    if factors is None:
        factors = (np.zeros(0, np.int64), np.zeros(0), np.zeros(1, np.int64), np.zeros(0, np.int64))
    fk, fc, fs, fm = (
        np.asarray(factors[0], np.int64),
        np.asarray(factors[1], np.float64),
        np.asarray(factors[2], np.int64),
        np.asarray(factors[3], np.int64),
    )
    theta = np.where(cont, cw[:, None] + gap_bonus, np.nan)
    ca, cb = np.asarray(cont_a, np.int64), np.asarray(cont_b, np.int64)
    c_bonus, c_change = np.asarray(cont_bonus, np.float64), np.asarray(cont_change, np.float64)
    # the labelling without the continuations that do not vouch (beside the frame's): a slit
    # that differs there rests on them alone
    keep = None if cont_ties is None or np.all(cont_ties) else np.asarray(cont_ties, bool)
    sel = keep if keep is not None else np.zeros(len(ca), bool)
    belief, alone = launch(
        _propagate_pair,
        np.ascontiguousarray(u, np.float64),
        np.asarray(gap_a, np.int64),
        np.asarray(gap_b, np.int64),
        np.ascontiguousarray(theta, np.float64),
        repeat_penalty * w,
        split_penalty * w,
        ca,
        cb,
        c_bonus,
        c_change,
        ca[sel],
        cb[sel],
        c_bonus[sel],
        c_change[sel],
        keep is not None,
        fk,
        fc,
        fs,
        fm,
    )
    best = np.argmax(belief, axis=1)
    top = belief[np.arange(s), best]
    with np.errstate(over="ignore"):
        conf = 1.0 / np.exp(belief - top[:, None]).sum(axis=1)
    # the groups of pieces the labelling ties together, and the dots' evidence of each
    ga, gb = np.asarray(gap_a, np.int64), np.asarray(gap_b, np.int64)
    tied_gap = (best[gb] == best[ga] + 1) & cont[np.arange(len(ga)), np.minimum(best[ga], n - 1)]
    tied_cont = best[ca] == best[cb]
    if cont_ties is not None:
        tied_cont &= np.asarray(cont_ties, bool)
    group = _groups(s, np.r_[ga[tied_gap], ca[tied_cont]], np.r_[gb[tied_gap], cb[tied_cont]])
    own = u[np.arange(s), best]
    support = np.bincount(group, weights=own, minlength=s)[group]
    rests = np.zeros(s, bool) if keep is None else np.argmax(alone, axis=1) != best
    conf = np.where(rests, 0.0, conf)
    ruled_out = ~np.isfinite(unary[np.arange(s), best])
    slit = np.where(ruled_out, -1, best)
    return Labelling(slit.astype(np.int64), conf, belief, support, rests & ~ruled_out)


def _groups(n: int, a: I64, b: I64) -> I64:
    """(n,) int64: the connected component of each of n nodes joined by the edges (a, b)."""
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def confidence_margin(confidence: float) -> float:
    """The margin (nats) over all other labels that a confidence (0..1) takes."""
    c = min(max(float(confidence), 1e-12), 1.0 - 1e-12)
    return math.log(c / (1.0 - c))
